"""A disk cache of predicted depth maps keyed by model + image file identity, so a split is predicted once."""

from __future__ import annotations

import hashlib
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from ..data.io import publish

__all__ = ["DepthCache"]


class DepthCache:
    """A disk cache of predicted depth maps: ``root/<model slug>/<ab>/<sha1>.npy``.

    The key covers the model, the image's absolute path, its modification time and size (an edited image is
    predicted again) and any ``extra`` input such as the focal length used.

    Args:
        root: The cache folder.
        model_id: The network's id (part of every key).
        dtype: How maps are stored: ``float16`` (1 mm at 2 m, 1 cm at 20 m, half the disk) or ``float32``.
    """

    def __init__(self, root: str | os.PathLike, model_id: str, dtype: str = "float16") -> None:
        self.model_id = model_id
        slug = re.sub(r"[^A-Za-z0-9._-]+", "_", model_id).strip("_")[-80:] or "model"
        self.dir = Path(root).expanduser() / slug
        self.dtype = np.dtype(dtype)
        self.hits = 0
        self.misses = 0

    def path(self, image_path: str | os.PathLike, extra: str = "") -> Path:
        """Where an image's map is cached.

        Args:
            image_path: The image file.
            extra: Any other input of the prediction (``fx=…``).

        Returns:
            The ``.npy`` path (not necessarily existing).
        """
        p = Path(image_path).resolve()
        st = p.stat()
        key = hashlib.sha1(f"{self.model_id}|{p}|{st.st_mtime_ns}|{st.st_size}|{extra}".encode()).hexdigest()
        return self.dir / key[:2] / f"{key}.npy"

    def round_trip(self, depth: np.ndarray) -> np.ndarray:
        """What a later ``get`` returns for ``depth``, so that the first answer equals every cached one.

        Args:
            depth: (H, W) metres.

        Returns:
            (H, W) float32, through the storage dtype.
        """
        return depth.astype(self.dtype).astype(np.float32)

    def get(self, path: Path) -> np.ndarray | None:
        """A cached map (counted in ``hits``), or None (absent or torn: counted in ``misses``).

        Args:
            path: From ``path``.

        Returns:
            (H, W) float32 metres, or None.
        """
        try:
            d = np.load(path, allow_pickle=False)
        except (OSError, ValueError):  # absent, or a torn write from a killed run: predict again
            self.misses += 1
            return None
        self.hits += 1
        return d.astype(np.float32)

    def put(self, path: Path, depth: np.ndarray) -> None:
        """Store a map atomically (readers never see half a file).

        Args:
            path: From ``path``.
            depth: (H, W) metres.
        """
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npy")
        with os.fdopen(fd, "wb") as f:
            np.save(f, depth.astype(self.dtype), allow_pickle=False)
        publish(tmp, path)  # atomic: readers never see half a file
