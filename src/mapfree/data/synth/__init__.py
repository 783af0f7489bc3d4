"""Synthetic Map-free scenes: textured places of interest rendered in numpy, written in the dataset's layout.

``generate(root, split)`` writes scenes that every part of mapfree (matching, solvers, training, scoring,
the service, the demo) can run on without the real dataset: real-photo textures, per-frame intrinsics,
metric ground-truth depth (suffix ``sensor``), a simulated monocular estimate (suffix ``mono``),
lighting changes between scans, and ``overlaps.npz`` for train scenes.
"""

from .depth import MonoDepthModel, simulate_mono_depth
from .generate import EST_DEPTH_SUFFIX, GT_DEPTH_SUFFIX, SynthOptions, generate, generate_scene
from .overlap import depth_overlap

__all__ = [
    "GT_DEPTH_SUFFIX",
    "EST_DEPTH_SUFFIX",
    "SynthOptions",
    "generate",
    "generate_scene",
    "MonoDepthModel",
    "simulate_mono_depth",
    "depth_overlap",
]
