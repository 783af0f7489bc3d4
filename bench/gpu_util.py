"""GPU utilisation over a block of work, sampled by ``nvidia-smi`` (``bench_pipeline.py``, ``baseline_loops.py``,
``bench_train.py``)."""

from __future__ import annotations

import contextlib
import subprocess
import threading

import numpy as np


class GpuUtilisation:
    """Mean GPU utilisation (%) over a ``with`` block, sampled by ``nvidia-smi`` every 100 ms; None without one."""

    def __enter__(self) -> GpuUtilisation:
        self.samples: list[float] = []
        self._proc = None
        try:
            self._proc = subprocess.Popen(
                ["nvidia-smi", "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits", "-lms", "100"],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )
        except (FileNotFoundError, PermissionError):
            return self
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()
        return self

    def _read(self) -> None:
        for line in self._proc.stdout:  # type: ignore[union-attr]
            with contextlib.suppress(ValueError):
                self.samples.append(float(line.split(",")[0]))

    def __exit__(self, *exc) -> None:
        if self._proc is not None:
            self._proc.terminate()
            self._proc.wait()

    @property
    def mean(self) -> float | None:
        return float(np.mean(self.samples)) if self.samples else None
