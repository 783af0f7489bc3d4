"""Relocalization for the service: a per-process pool of ``Relocalizer`` objects per method and an LRU of
prepared anchors (reference features and depth are computed once per anchor and method)."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Hashable, Iterable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import cv2
import numpy as np
from fastapi import Depends, Request

from ...calibration import Calibration
from ...estimate import Estimate
from ...geometry import Intrinsics
from ...matching.base import Matches
from ..inputs import UploadError
from .calibration import calibrate, source_of
from .methodpool import MethodPool
from .photos import Photo
from .prepared import ByteLRU, PreparedAnchor, localize_prepared, prepare_anchor
from .worksize import DEFAULT_MAX_SIDE, fit_photo

if TYPE_CHECKING:
    from ...methods import Method
    from ...relocalize import Localizer

log = logging.getLogger("mapfree.service")
FALLBACK_METHOD = "sift_pnp_sensor"  # reference depth only: what an anchor with a depth map can always use


def default_method(configured: str = "") -> str:
    """The configured method, else the registry's best offline preset, else SIFT + PnP on the anchor's depth."""
    from ... import methods

    for name in (configured, methods.BEST_OFFLINE, FALLBACK_METHOD):
        if not name:
            continue
        try:
            methods.get(name)
            return name
        except (KeyError, ValueError, FileNotFoundError):
            continue
    return FALLBACK_METHOD


#: What a method name sent over HTTP may look like: never a path, a ``NAME@DEPTH`` override or a depth spec
#: with a colon (those would make the server read files the client chooses).
METHOD_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")
#: Depth-file suffixes a preset name may carry: in the service every one of them means the depth map uploaded
#: with the photo (the dataset's files are never read), so any other suffix names no depth a request can have.
DEPTH_SUFFIXES = ("sensor", "dptkitti", "dptnyu", "mono")


def allowed_methods() -> str:
    """The names a client may send, for error messages: registered names and YAML configs, and the preset pattern."""
    from ... import matching, methods

    named = ", ".join(methods.list_methods(depths=()))
    return (
        f"{named}; or a preset {{matcher}}_{{emat|pnp|procrustes}}_{{depth}} with matcher in "
        f"{', '.join(matching.available())} and depth 'none' or a depth-file suffix such as 'sensor'"
    )


def check_method(name: str) -> str:
    """A method name from a client -> the registered name. Only registered names, the project's and the
    operator's YAML configs (by name) and ``{matcher}_{solver}_{depth}`` presets: never a path, so a client
    cannot make the server open, parse or probe files. Anything else is a 422 listing what is allowed."""
    from ... import methods

    name = name.strip()
    ok = METHOD_NAME_RE.fullmatch(name) is not None and not name.lower().endswith((".yaml", ".yml"))
    if ok:
        try:
            m = methods.get(name)
        except (KeyError, ValueError, FileNotFoundError, OSError):
            pass
        else:
            suffix = m.depth[len("files:") :] if m.kind == "matching" and m.depth.startswith("files:") else ""
            if suffix and suffix not in DEPTH_SUFFIXES:
                raise UploadError(
                    422,
                    f"method: {name[:64]!r} names depth files '.{suffix[:20]}.png', which a "
                    "request cannot carry: the depth here is the map uploaded with the photo; "
                    f"use the suffix {' or '.join(DEPTH_SUFFIXES)} (e.g. "
                    f"{m.matcher}_{m.solver.replace('essential', 'emat')}_sensor)",
                )
            return m.name
    raise UploadError(422, f"method: unknown method {name[:64]!r}; allowed: {allowed_methods()}")


def register_methods_dir(folder) -> list[str]:
    """Register every ``*.yaml`` of the operator's methods folder by its name (``--methods-dir``)."""
    from ... import methods

    names = []
    for p in sorted(Path(folder).glob("*.y*ml")):
        if not METHOD_NAME_RE.fullmatch(p.stem):
            continue
        try:
            methods.register(replace(methods.load_yaml(p), name=p.stem), overwrite=True)
            names.append(p.stem)
        except (ValueError, KeyError, FileNotFoundError, OSError) as e:
            log.warning("method config skipped", extra={"file": str(p), "error": str(e)})
    return names


class MethodUnavailable(UploadError):
    """A known method that cannot run here (weights missing, no depth where it needs one)."""

    def __init__(self, message: str):
        super().__init__(422, message)


def needs_reference_depth(method: Any, *, scale_free_too: bool) -> bool:
    """Whether ``method`` (a name or ``Method``) needs a depth map uploaded with the reference photo.

    Always for matching methods whose depth comes from files (``files:SUFFIX``): that map is their metric scale.
    ``scale_free_too`` also counts methods without depth (``none``) whose solver is PnP or Procrustes: with an
    uploaded map they run (at its scale), without one every query fails. An anchor is refused for those
    (``check_runnable``: it would never localize); the one-off try page lets them run and shows the failure.
    Predicted-depth (a network), Ess.Mat-without-depth and regression methods never need one."""
    from ... import methods

    m = method if isinstance(method, methods.Method) else methods.get(method)
    if m.kind != "matching":
        return False
    # Without a depth map, PnP/Procrustes give no pose at all, even in a method with no depth source ("none"),
    # which then uses a depth map uploaded with the reference.
    lifting = m.depth == "none" and m.solver in methods.LIFTING_SOLVERS
    return m.depth.startswith("files:") or (scale_free_too and lifting)


def check_runnable(name: str, has_reference_depth: bool) -> None:
    """Refuse (422) an anchor whose method can never localize it: a reference-depth method without a depth map."""
    if not has_reference_depth and needs_reference_depth(name, scale_free_too=True):
        raise MethodUnavailable(
            f"method {name} takes its metric scale from the anchor's depth map, and this anchor has none: upload "
            "'depth' (a single-channel uint16 PNG in millimetres), or choose a method that works without depth "
            "(e.g. sift_emat_none: scale-free pose; or a monocular depth network such as xfeat_pnp_dpt-kitti)"
        )


def _unavailable(name: str, e: Exception) -> MethodUnavailable:
    """Why a method cannot be built here, naming missing weights without the server's folders."""
    from ...matching import MissingWeightsError

    if isinstance(e, MissingWeightsError):
        m = re.search(r"weights file '([^']+)'", str(e))
        what = str(e).split(":", 1)[0]
        return MethodUnavailable(
            f"method {name} cannot run on this server: the {what} weights "
            f"({m.group(1) if m else 'file'}) are missing; ask the operator to install them"
        )
    msg = str(e).split(" (", 1)[0][:200] if isinstance(e, (ValueError, KeyError, ImportError)) else type(e).__name__
    return MethodUnavailable(f"method {name} cannot run on this server: {msg}")


def effective_method(name: str, has_query_depth: bool) -> Method:
    """The ``Method`` to run: ``name``, or its PnP twin when the query has no depth map but the method's solver
    would need one (so that the default preset answers for a plain photo, at the anchor's metric scale)."""
    from ... import methods

    m = methods.get(name)
    return m if has_query_depth else methods.query_depth_fallback(m)


class Localizers:
    """Thread-safe access to relocalizers: at most ``per_method`` concurrent computations per method.

    Every photo is at the working size (long side at most ``max_side``, ``worksize.fit_photo``) when a method
    sees it (``photos.read_upload`` brings uploads there; ``fit`` makes sure of the rest). Prepared anchors
    (``prepared.py``: features and depth per photo, no pixels) are kept per (anchor, method, version) in an LRU
    of at most ``cache_bytes``. The version names the anchor's current photos (``domain.anchor_version``: it
    changes when one is added or deleted), so a change made through another
    process is never answered from a stale cache. Built relocalizers live in a ``MethodPool`` of at most
    ``pool_bytes``, shared by equal configurations (``methodpool.py``)."""

    def __init__(
        self,
        per_method: int = 2,
        cache_bytes: int = 256 << 20,
        max_side: int = DEFAULT_MAX_SIDE,
        pool_bytes: int = 1 << 30,
    ):
        self.max_side = max_side
        self.pool = MethodPool(self._build, per_method, pool_bytes)
        self.anchors = ByteLRU(cache_bytes)

    def fit(self, photo: Photo) -> Photo:
        """``photo`` at the working size (intrinsics and depth scaled with it)."""
        return fit_photo(photo, self.max_side)

    @staticmethod
    def _build(method: Method) -> Localizer:
        from ...relocalize import build_localizer
        from ...relocalize.allocator import keep_heap_warm

        keep_heap_warm()  # this process relocalizes: per-pair buffers stay in its heap (once per process)
        try:
            return build_localizer(method)
        except Exception as e:
            raise _unavailable(method.name, e) from e

    def _take(self, method: Method) -> Localizer:
        return self.pool.take(method)

    def _give(self, method: Method, loc: Localizer) -> None:
        self.pool.give(method, loc)

    def _prepare(self, loc: Localizer, name: str, photos: Iterable[Photo]) -> PreparedAnchor:
        """Every photo prepared at the working size (``prepared.prepare_anchor``; each one fitted as it comes,
        so that a generator of decoded photos holds one at its native size at a time); a method that cannot
        run here is a 422, not a 500."""
        try:
            return prepare_anchor(loc, [self.fit(p) for p in photos])
        except Exception as e:  # e.g. a depth network whose weights are gone
            raise _unavailable(name, e) from e

    def check(
        self, anchor_id: str, method: str, photos: list[Photo], version: Hashable = (), owner: Hashable = None
    ) -> None:
        """Build the method and prepare the anchor now (both kept for the first ``localize``), so that an
        anchor whose method cannot run here is refused at creation (``MethodUnavailable``), not at use."""
        plain, with_depth = effective_method(method, False), effective_method(method, True)
        for i, m in enumerate([plain] if plain.name == with_depth.name else [plain, with_depth]):
            loc = self._take(m)
            try:
                if i > 0:
                    continue  # built (weights present); the reference is prepared once, by the usual variant
                prepared = self._prepare(loc, m.name, photos)
                self.anchors.put((anchor_id, m.name, version), prepared, prepared.nbytes, owner)
            finally:
                self._give(m, loc)

    def forget(self, anchor_id: str) -> None:
        self.anchors.drop(lambda k: k[0] == anchor_id)

    def localize(
        self,
        anchor_id: str,
        method: str,
        ref_image: np.ndarray,
        ref_K: Intrinsics,
        ref_depth: np.ndarray | None,
        query_image: np.ndarray,
        query_K: Intrinsics,
        query_depth: np.ndarray | None = None,
        owner: Hashable = None,
    ) -> Estimate:
        """Pose of the query relative to one reference photo; ``est.extras["method"]`` names what ran."""
        return self.localize_photos(
            anchor_id,
            method,
            (),
            lambda: [Photo(ref_image, ref_K, ref_depth)],
            query_image,
            query_K,
            query_depth,
            owner,
        )

    def localize_photos(
        self,
        anchor_id: str,
        method: str,
        version: Hashable,
        photos: Callable[[], Iterable[Photo]],
        query_image: np.ndarray,
        query_K: Intrinsics,
        query_depth: np.ndarray | None = None,
        owner: Hashable = None,
        calibrations: Mapping[str, Calibration] | None = None,
    ) -> Estimate:
        """World-to-camera pose of the query in the anchor's frame. ``photos`` is called (decoding the stored
        images) only when this process has not prepared this version of the anchor yet; what it prepares counts
        against ``owner``'s share of the cache (the account asking: ``prepared.ByteLRU``). With several photos
        ``est.photo`` is the retrieved one (``est.extras``: ``retrieval_similarity``). Keypoints in ``est.matches``
        are in the working-size pixels (``fit``). The estimate carries ``p_correct`` from the anchor's
        ``calibrations`` (by method name), else the method's shipped one (``calibration.calibrate``), and
        ``extras["calibration"]`` says which."""
        chosen = effective_method(method, query_depth is not None)
        loc = self._take(chosen)
        try:
            key = (anchor_id, chosen.name, version)
            prepared = self.anchors.get(key)
            if prepared is None:
                prepared = self._prepare(loc, chosen.name, photos())
                self.anchors.put(key, prepared, prepared.nbytes, owner)
            q = self.fit(Photo(query_image, query_K, query_depth))
            try:
                cals = calibrations or {}
                est = localize_prepared(calibrate(loc, chosen.name, cals), prepared, q)
            except MethodUnavailable:
                raise
            except Exception as e:  # a method that fails outright on this input (not a "no pose")
                raise _unavailable(chosen.name, e) from e
            est.extras["method"] = chosen.name
            est.extras["calibration"] = source_of(est, chosen.name, cals)
            return est
        finally:
            self._give(chosen, loc)


async def _localizers(request: Request) -> Localizers:  # async: resolving it takes no thread of the shared pool
    return request.app.state.localizers


#: A route's ``localizers: LocalizersDep``: the app's prepared methods (``create_app`` holds them).
LocalizersDep = Annotated[Localizers, Depends(_localizers)]


def estimate_json(est: Estimate, method: str) -> dict:
    d = est.to_dict()
    d["method"] = est.extras.get("method", method)
    d["num_matches"] = int(est.extras.get("num_matches", 0) or 0)
    d["scale_free"] = bool(est.extras.get("scale_free", False))
    if est.photo is not None:  # which photo of the anchor answered (0: its first)
        d["photo"] = int(est.photo)
    if "retrieval_similarity" in est.extras:
        d["retrieval_similarity"] = float(est.extras["retrieval_similarity"])
    if est.extras.get("calibration"):
        d["calibration"] = est.extras["calibration"]
    return d


def figure_png(
    ref_image: np.ndarray,
    query_image: np.ndarray,
    ref_K: Intrinsics,
    query_K: Intrinsics,
    est: Estimate,
    title: str = "",
) -> bytes:
    """Matches on top and the virtual grid rendered into the query at the estimated pose below, as PNG bytes."""
    from ... import viz

    m = est.matches if est.matches is not None else Matches.empty()  # none: RPR, or a failure before matching
    k0, k1 = m.kpts0, m.kpts1
    fig = viz.relocalization_figure(
        ref_image, query_image, ref_K, query_K, k0, k1, est.pose, title=title, reason=est.reason
    )
    ok, buf = cv2.imencode(".png", cv2.cvtColor(fig, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("could not encode the figure")
    return buf.tobytes()
